"""A law prior's step scripted alone (test_fe_modes): its dense path in TorchScript, without a
LinearPriorModel and its network around it."""

from typing import Tuple

from torch import Tensor, nn


class PriorStep(nn.Module):
    """``prior.step`` (a ``HyperelasticNewmarkPrior``'s) as a module's forward, to script it."""

    def __init__(self, prior: nn.Module) -> None:
        super().__init__()
        self.prior = prior

    def forward(self, u0: Tensor, v0: Tensor, a0: Tensor, f1: Tensor, G0: Tensor, G1: Tensor,
                h0: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        return self.prior.step(u0, v0, a0, f1, G0, G1, h0)
