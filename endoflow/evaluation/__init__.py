"""Test-set evaluation (depth and pose metrics, the latent bank's SWD, plots); never imports training."""
