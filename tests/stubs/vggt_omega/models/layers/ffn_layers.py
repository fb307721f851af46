from typing import Callable, Optional

from torch import Tensor, nn


class Mlp(nn.Module):
    """fc1 -> activation -> fc2 (parameter names as upstream)."""

    def __init__(
        self,
        in_features: int,
        hidden_features: Optional[int] = None,
        out_features: Optional[int] = None,
        act_layer: Callable[..., nn.Module] = nn.GELU,
        drop: float = 0.0,
        bias: bool = True,
        device=None,
    ) -> None:
        super().__init__()
        self.fc1 = nn.Linear(in_features, hidden_features or in_features, bias=bias, device=device)
        self.act = act_layer()
        self.fc2 = nn.Linear(
            hidden_features or in_features, out_features or in_features, bias=bias, device=device
        )

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(self.act(self.fc1(x)))
