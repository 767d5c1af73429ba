"""One clipped-PPO mini-batch step on a TorchRL loss, shared by MAPPO (:mod:`cv2x_marl.rl.mappo`) and the TorchRL
PPO loop (:mod:`cv2x_marl.rl.fast_ppo`)."""

from __future__ import annotations

from typing import Any

#: the loss terms a step adds up and reports (``loss_entropy`` only where the loss has an entropy term)
LOSS_KEYS = ("loss_objective", "loss_critic", "loss_entropy")


def ppo_minibatch_step(
    loss: Any, batch: Any, optim: Any, params: list[Any], max_grad_norm: float, sums: dict[str, float]
) -> None:
    """Minimise ``loss(batch)``'s objective + critic (+ entropy) terms with one step of ``optim``, the gradient's
    norm clipped to ``max_grad_norm`` over ``params``; add each term's value to ``sums`` (keys :data:`LOSS_KEYS`).

    Args:
        loss: a TorchRL loss module (``ClipPPOLoss``) returning a TensorDict of ``loss_*`` terms.
        batch: the mini-batch (a TensorDict).
        optim: the optimizer over ``params``.
        params: the parameters whose gradient norm is clipped.
        max_grad_norm: the clip (PPO's ``max_grad_norm``).
        sums: running sums of the loss terms, updated in place.
    """
    import torch

    out = loss(batch)
    total = out["loss_objective"] + out["loss_critic"]
    if "loss_entropy" in out.keys():
        total = total + out["loss_entropy"]
    optim.zero_grad()
    total.backward()
    torch.nn.utils.clip_grad_norm_(params, max_grad_norm)
    optim.step()
    for key in sums:
        if key in out.keys():
            sums[key] += float(out[key].detach())
