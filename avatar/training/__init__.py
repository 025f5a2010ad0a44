"""Training loops of the avatar: the warm-up (stage one), stage two (the dynamic model), SplattingAvatar's."""
