"""The app's sweeper (``hydra/sweeper=interactavatar``): Hydra finds sweepers only under ``hydra_plugins``."""
