"""The project's Hydra launcher plugins (Hydra finds launchers only under the ``hydra_plugins`` package)."""
