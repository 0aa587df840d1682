"""Networks: latent bank generator, critic, depth encoder/decoder, pose network, joint model."""
