"""The query protocol (``eval.query_protocol``): prototype frames drawn per class by seed, nearest-prototype labels of
held-out frames scored per feature source, a feature space that separates the classes scoring mIoU 1, off by default,
and on a tiny GP-NeRF through ``evaluate`` beside the class head's mIoU."""

from __future__ import annotations

import pytest
import torch

from gpnerf_core.config.compose import compose
from gpnerf_core.data.frames import FrameCache
from gpnerf_core.errors import ConfigError
from gpnerf_core.evaluation import metrics as M
from gpnerf_core.evaluation.evaluator import evaluate, print_summary
from gpnerf_core.evaluation.query_protocol import QueryProtocol, prototype_frames
from gpnerf_core.model.build import build_components
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.types import Prediction
from pipeline_check import TINY_MODEL, TINY_SCENES


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A tiny untrained GP-NeRF with a class head (seeded) on the tiny embedded scenes, one held-out view per scene."""
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("rooms")
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={root}",
                   "eval.max_views_per_scene=1", "eval.save_images=0"])
    torch.manual_seed(0)
    components = build_components(cfg)
    return cfg, components, FrameCache(components.dataset, torch.device("cpu"))


def test_prototype_frames_are_k_frames_showing_each_class_drawn_by_seed(tiny):
    _, components, frames = tiny
    scene = frames.scene(components.dataset.scenes("train")[0])
    labels = {i: frames.frame(scene, i).semantic for i in scene.train_frames}
    K = components.classes.num_classes
    once = prototype_frames(scene, labels, K, 2, seed=0)
    assert once == prototype_frames(scene, labels, K, 2, seed=0)  # deterministic
    for value, indices in once.items():
        assert 1 <= len(indices) <= 2 and len(set(indices)) == len(indices)
        assert all(i in scene.train_frames and bool((labels[i] == value).any()) for i in indices)
        shown_by = [i for i in scene.train_frames if bool((labels[i] == value).any())]
        assert len(indices) == min(2, len(shown_by))
    assert set(once) == {v for i in scene.train_frames for v in labels[i].unique().tolist() if 0 <= v < K}
    draws = {tuple(map(tuple, prototype_frames(scene, labels, K, 1, seed=s).values())) for s in range(6)}
    assert len(draws) > 1  # another seed, other frames


def one_hot_render(frames, num_classes, scene_frames):
    """A 'model' whose semantic embedding is the frame's labels one-hot (plus noise): a feature space that separates
    the classes, rendered at stride 2."""
    def render(scene, index):
        labels = frames.frame(scene, index).semantic[::2, ::2]
        features = torch.nn.functional.one_hot(labels.clamp(0, num_classes - 1), num_classes).permute(2, 0, 1).float()
        scene_frames.append(index)
        features = features + 0.01 * torch.randn_like(features)
        return Prediction(rgb=torch.zeros(*labels.shape, 3), depth=torch.ones(labels.shape), semantic=features,
                          logits=None, stride=2)
    return render


def test_a_feature_space_that_separates_the_classes_scores_miou_one(tiny):
    _, components, frames = tiny
    K = components.classes.num_classes
    rendered = []
    render = one_hot_render(frames, K, rendered)
    protocol = QueryProtocol(render=render, frames=frames, num_classes=K, ignore_index=components.dataset.ignore_index)
    scene = frames.scene(components.dataset.scenes("train")[0])
    index = scene.eval_frames[0]
    target = frames.frame(scene, index)
    confusions = protocol.confusions(scene, index, target, render(scene, index))
    assert set(confusions) == {"semantic_embedding"}
    # the stride-2 labels on the image differ from the real labels at class edges only
    grid = target.semantic[::2, ::2].repeat_interleave(2, 0).repeat_interleave(2, 1)
    expected = M.confusion_matrix(grid, target.semantic, K, components.dataset.ignore_index)
    assert torch.equal(confusions["semantic_embedding"], expected)
    own = M.image_scores_from_confusion(M.confusion_matrix(grid, grid, K))
    assert own[M.MIOU_IMAGE_MEAN_PRESENT] == 1.0
    before = len(rendered)
    protocol.confusions(scene, index, target, render(scene, index))
    assert len(rendered) == before + 1  # the prototypes are taken once per scene: only the held-out frame again
    with pytest.raises(ConfigError, match=r"eval.prototype_frames=0: expected an integer >= 1"):
        QueryProtocol(render=render, frames=frames, num_classes=K, ignore_index=255, k=0)


def test_the_protocol_is_off_by_default_and_scored_beside_the_head_when_asked(tiny, tmp_path, capsys):
    cfg, components, frames = tiny
    cfg = cfg.copy()
    cfg.eval.splits = ["train"]
    off = evaluate(cfg, components, frames, tmp_path / "off", Distributed.single())["eval"]["train_heldout"]
    assert M.QUERY_PROTOTYPE not in off
    cfg.eval.query_protocol = True
    on = evaluate(cfg, components, frames, tmp_path / "on", Distributed.single())["eval"]["train_heldout"]
    query = on[M.QUERY_PROTOTYPE]
    assert query["prototype_frames"] == 1 and query["seed"] == 0 and list(query["sources"]) == ["semantic_embedding"]
    scored = query["sources"]["semantic_embedding"]
    assert 0.0 <= scored[M.MIOU_IMAGE_MEAN_PRESENT] <= 1.0 and scored[M.COUNT_IMAGES] == 1
    for key in (*M.SEGMENTATION_KEYS, "baseline_majority"):  # the head's numbers do not change
        assert on[key] == off[key], key
    print_summary({"eval": {"train_heldout": on}}, tmp_path)
    assert "| query by prototype (1 frame/class) mIoU: semantic_embedding " in capsys.readouterr().out
