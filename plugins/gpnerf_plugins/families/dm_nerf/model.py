"""DM-NeRF (Wang et al., ICLR 2023; official code ``vLAR-group/DM-NeRF``) as a per-scene instance family.

NeRF's field of one scene (``families/nerf_field.py``: the positional encoding without scaling, trunk with a skip,
density, view-dependent colour; coarse and fine networks) plus DM-NeRF's **object field**: on the trunk features,
**detached** (instance gradients never shape the geometry), ``Linear(width, width)``, ``Linear(width, width / 2)``,
ReLU, ``Linear(width / 2, K + 1)``: K object slots and an "empty" one. The object logits are composited along the ray
with the **detached** weights; the slot probabilities are each slot's own **sigmoid after** compositing (no softmax
across slots), the empty slot dropped: ``SemanticOutput.slot_activation = "sigmoid"``. The per-sample logits go to the
loss set (``RenderedRays.sample_semantic``) for DM-NeRF's 3D emptiness penalty (``losses/dm_nerf.py``).

What changed for two CPU cores, as for Semantic-NeRF (``families/semantic_nerf``): width 256 -> 128, trunk 8 -> 6
(the skip kept), samples 64 + 128 -> 32 + 32, 3072 -> 512 rays a step, and the step budget (500k official).
"""

from __future__ import annotations

from torch import Tensor, nn

from gpnerf_core import ConfigError, Predicts, SemanticMode, SemanticOutput, composite
from gpnerf_plugins.families.nerf_field import PerSceneNeRF


def object_branch(width: int, slots: int) -> nn.Module:
    """DM-NeRF's object head: ``Linear(width, width)``, ``Linear(width, width / 2)``, ReLU, ``Linear(width / 2,
    slots + 1)``."""
    return nn.Sequential(nn.Linear(width, width), nn.Linear(width, width // 2), nn.ReLU(),
                         nn.Linear(width // 2, slots + 1))


class DMNeRF(PerSceneNeRF):
    """DM-NeRF: coarse and fine fields of one scene with an object field on their detached trunk features (module
    docstring).

    Args:
        slots: K object slots (K + 1 outputs, the last "empty").
        the rest: ``DMNeRFConfig``'s (``PerSceneNeRF``).
    """

    def __init__(self, *, slots: int, **field: float | int | bool) -> None:
        if isinstance(slots, bool) or not isinstance(slots, int) or slots < 1:
            raise ConfigError(f"model.slots={slots!r}: expected an integer >= 1 (object slots)")
        self.slots = slots
        super().__init__(**field, detach_branch=True)

    def make_branch(self, width: int) -> nn.Module:
        return object_branch(width, self.slots)

    def composite_branch(self, weights: Tensor, outputs: Tensor) -> Tensor:
        """DM-NeRF renders the object logits with fixed (detached) weights."""
        return composite(weights.detach(), outputs)

    @property
    def semantic_output(self) -> SemanticOutput:
        return SemanticOutput(Predicts.INSTANCES, SemanticMode.LABEL_RENDERING, self.slots + 1, self.slots,
                              slot_activation="sigmoid")
