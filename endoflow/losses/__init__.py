"""Training losses: photometric reprojection (:mod:`.photometric`), edge-aware smoothness
(:mod:`.smoothness`), KL to a standard normal (:mod:`.kl`) and WGAN-GP (:mod:`.gan`)."""
