"""The DAG runner: stage registry, cache keys, manifests, atomic writes, locks, CLI."""
