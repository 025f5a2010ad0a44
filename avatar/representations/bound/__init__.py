"""Gaussians bound to the FLAME and MANO triangles (GaussianAvatars; InteractAvatar and its ablations): the
container and its density control (``gaussians``, ``density``), the static warm-up (``warmup``), InteractAvatar's
pose-dependent hand and interaction modules (``dynamic_model``) and their training (``stage_two``), and the
representation the training stages call (``representation``: loading, posing a frame, artifacts)."""
