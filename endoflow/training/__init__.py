"""Latent-bank pretraining, the self-supervised objective and the distributed training loop."""
