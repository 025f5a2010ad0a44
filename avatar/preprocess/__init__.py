"""Image preprocessing shared by stages: foreground masks, part boxes, square crops with adjusted intrinsics."""
