"""Semantic-NeRF (Zhi et al., ICCV 2021; official code ``Harry-Zhi/semantic_nerf``) as a per-scene family.

One scene's field, fitted on that scene's training frames and rendered from its own parameters (no source views):

- **Encoding**: positions multiplied by ``position_scale`` (the official code divides by 10), then NeRF's positional
  encoding ``[x, sin(2^k x), cos(2^k x)]``, k < 10 (63 channels); unit view directions with 4 octaves (27 channels).
- **Trunk**: ``depth`` ReLU layers of ``width``, the encoded position concatenated after layer ``skip``.
- **Heads**: density ``Linear(width, 1)``, raw (ReLU at render time, after noise of std ``density_noise`` in training);
  semantics ``Linear(width, width/2)``, ReLU, ``Linear(width/2, K)``, view-independent; colour ``Linear(width, width)``
  concatenated with the encoded direction, ``Linear(. , width/2)``, ReLU, ``Linear(width/2, 3)``, sigmoid.
- **Rendering**: ``alpha = 1 - exp(-ReLU(sigma) * delta * |d|)`` with the last interval 1e10; colour, depth and the
  class **logits** composited with the weights (label rendering); the prediction is their argmax.
- **Coarse and fine**: separate networks; ``coarse_samples`` stratified samples uniform in depth between near and far
  (jittered in training), the fine network on those plus ``fine_samples`` importance samples of the coarse weights.
- **Loss** (the experiment ``baselines/semantic_nerf``): colour MSE of both passes + 0.04 x cross-entropy of both.

What changed for two CPU cores (each also in ``SemanticNeRFConfig``): width 256 -> 128, trunk 8 -> 6 layers (the skip
kept), samples 64 + 128 -> 32 + 32, 1024 -> 256 rays a step, and the step budget (the official 200k steps take hours on
a GPU). The classes are the dataset's, not remapped per scene as the official loaders do (a scene's absent classes are
simply never predicted there; the metrics score present classes, as for every family here).
"""

from __future__ import annotations

from torch import nn

from gpnerf_core import Predicts, SemanticMode, SemanticOutput
from gpnerf_plugins.families.nerf_field import PerSceneNeRF


class SemanticNeRF(PerSceneNeRF):
    """Semantic-NeRF: coarse and fine fields of one scene with a view-independent semantic branch, label rendering
    (module docstring).

    Args:
        num_classes: K (0: colour and depth only).
        the rest: ``SemanticNeRFConfig``'s (``PerSceneNeRF``).
    """

    def __init__(self, *, num_classes: int, **field: float | int | bool) -> None:
        self.num_classes = int(num_classes)
        super().__init__(**field)

    def make_branch(self, width: int) -> nn.Module | None:
        """``Linear(width, width / 2)``, ReLU, ``Linear(width / 2, K)`` on the trunk features (not detached)."""
        if not self.num_classes:
            return None
        return nn.Sequential(nn.Linear(width, width // 2), nn.ReLU(), nn.Linear(width // 2, self.num_classes))

    @property
    def semantic_output(self) -> SemanticOutput | None:
        if not self.num_classes:
            return None
        return SemanticOutput(Predicts.CLASSES, SemanticMode.LABEL_RENDERING, self.num_classes)
