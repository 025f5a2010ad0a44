"""InteractAvatar model core (importable without the pipeline)."""
