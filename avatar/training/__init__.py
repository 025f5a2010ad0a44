"""Training loops of the avatar (static warm-up; dynamic MLP training arrives later)."""
