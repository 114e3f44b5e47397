"""A model whose outputs hold NaN or Inf is stopped with an error naming the component, never scored."""

import pytest
import torch

from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.errors import NonFiniteError
from gpnerf_core.evaluation.evaluator import evaluate
from gpnerf_core.data.frames import FrameCache
from pipeline_check import TINY_MODEL, TINY_SCENES


@pytest.mark.parametrize("poisoned, named", [
    ("head", r"head 'unet' \(plugin gpnerf_plugins.heads.plugin, gpnerf-core [^)]*\) returned logits that are not "
             r"finite .* from finite input features; nothing was scored"),
    ("ray", r"ray aggregator 'gnt_ray' gave NaN or Inf \(colour\)"),
    ("semantic", r"head 'unet' .* from input features that were not finite already .*: the fault is upstream of it, "
                 r"in model 'gnt' \(plugin gpnerf_plugins.families.plugin, gpnerf-core [^)]*\), which made them"),
])
def test_non_finite_outputs_stop_evaluation_naming_the_component(tmp_path, poisoned, named):
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}",
                   "eval.splits=[unseen]", "eval.save_images=0"])
    components = build_components(cfg)
    module = {"head": components.model.head, "ray": components.model.ray,
              "semantic": components.model.semantic}[poisoned]
    with torch.no_grad():
        last = [p for p in module.parameters() if p.dim() >= 1][-1]
        last.fill_(float("inf") if poisoned == "ray" else float("nan"))
    components.model.eval()
    frames = FrameCache(components.dataset, torch.device("cpu"))
    with pytest.raises(NonFiniteError, match=r"scene '\w+' frame \d+: .*" + named):
        evaluate(cfg, components, frames, tmp_path / "run", Distributed.single())
    assert not (tmp_path / "run" / "metrics.json").exists()
