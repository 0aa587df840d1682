"""endoflow: self-supervised monocular depth and pose for endoscopy."""

__version__ = "0.1.0"
