"""The small model most tests build: the default network at a small input size, without the latent bank (which
needs a pretrained bank file)."""

from __future__ import annotations


from endoflow.config import Params


def small_model_params(size: int) -> Params:
    params = Params()
    params.data.size = size
    params.model = params.model.replace(latent_bank=False)
    return params
