"""Latent optimization (the paper's post-processing): freeze NNet, optimize the encoder's output
so the rendering layer reproduces the photos better; the decoder keeps normals plausible."""

from __future__ import annotations

import torch
from torch import Tensor

from ..config import LatentOptConfig  # noqa: F401 (re-exported; its home is lookingglass.config)
from ..physics.camera import Cameras
from ..physics.environment import EnvironmentMap
from .model import NormalNet
from ..physics.optics import IOR_GLASS
from .render_layer import comparable, render_layer


def masked_render_loss(envmap: EnvironmentMap, n1: Tensor, n2: Tensor, cameras: Cameras, image: Tensor,
                       mask: Tensor, view_dirs: Tensor | None = None, ior: float = IOR_GLASS) -> Tensor:
    """The paper's L = ||(I - (I^r + I^t)) ⊙ M^tr||², averaged over the usable pixels (in the mask
    and not TIR); the rendering is clipped like the input. n1, n2 (V,3,H,W) camera frame; image (V,H,W,3); mask (V,H,W)."""
    out = render_layer(envmap, n1.permute(0, 2, 3, 1), n2.permute(0, 2, 3, 1), cameras, ior=ior, view_dirs=view_dirs)
    usable = (mask & ~out.tir).unsqueeze(-1).to(image.dtype)
    return (((image - comparable(out.image)) * usable) ** 2).sum() / (usable.sum() * 3).clamp(min=1)


def adam_step(param: Tensor, moments: tuple[Tensor, Tensor], t: int, lr: float,
              betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> None:
    """One step of Adam (torch.optim.Adam's update, defaults) on `param` from its .grad, which it
    then clears; moments (m, v) are updated in place; t counts steps from 1.

    Why not torch.optim.Adam: creating one imports torch._dynamo, 2-3.5 s here, a tenth of
    `reconstruct`'s normal stage, for a single tensor's update (tests/test_latent.py checks that
    the two agree)."""
    m, v = moments
    with torch.no_grad():
        g = param.grad
        m.mul_(betas[0]).add_(g, alpha=1 - betas[0])
        v.mul_(betas[1]).addcmul_(g, g, value=1 - betas[1])
        denom = (v / (1 - betas[1] ** t)).sqrt_().add_(eps)
        param.addcdiv_(m, denom, value=-lr / (1 - betas[0] ** t))
    param.grad = None


def optimize_latent(net: NormalNet, inputs: Tensor, cost_volume: Tensor | None, envmap: EnvironmentMap,
                    image: Tensor, mask: Tensor, cameras: Cameras, config: LatentOptConfig | None = None,
                    ior: float = IOR_GLASS) -> tuple[Tensor, Tensor, list[float], Tensor | None]:
    """Returns the optimized (n1, n2), each (V,3,H,W), the loss after every step, and the gain
    head's prediction for the optimized normals (V,2,H,W; None without a head)."""
    config = config or LatentOptConfig()
    for p in net.parameters():
        p.requires_grad_(False)
    with torch.no_grad():
        latent0 = net.encode(inputs, cost_volume)
        n1_init, _ = net.decode(latent0, inputs)
    latent = latent0.clone().requires_grad_(True)
    moments = (torch.zeros_like(latent), torch.zeros_like(latent))
    dirs = cameras.pixel_rays()[1].to(image)
    m = mask.unsqueeze(1).to(image.dtype)
    history = []
    for step in range(config.iterations_n2 + config.iterations_both):
        n1, n2 = net.decode(latent, inputs)
        loss = masked_render_loss(envmap, n1, n2, cameras, image, mask, view_dirs=dirs, ior=ior)
        history.append(float(loss.detach()))
        if step < config.iterations_n2:
            loss = loss + config.identity_weight * (((n1 - n1_init) * m) ** 2).sum() / (m.sum() * 3).clamp(min=1)
        loss.backward()
        adam_step(latent, moments, step + 1, config.lr)
    with torch.no_grad():
        n1, n2, gain = net.decode_with_gain(latent, inputs)
        history.append(float(masked_render_loss(envmap, n1, n2, cameras, image, mask, view_dirs=dirs, ior=ior)))
    return n1, n2, history, gain
