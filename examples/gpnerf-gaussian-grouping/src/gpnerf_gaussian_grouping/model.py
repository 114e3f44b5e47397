"""Gaussian Grouping (Ye, Danelljan, Yu, Ke; ECCV 2024; ``lkeab/gaussian-grouping@0ab60af``) on gpnerf-core's public
per-scene Gaussian family (``GaussianFamily``): 3D Gaussian splatting with an identity encoding per Gaussian.

- **Identity**: ``identity_dim`` raw floats per Gaussian (``_objects_dc``), started ``RGB2SH(U(0, 1))``, cloned and
  split with its Gaussian, composited like colour without a background term; a ``Conv2d(identity_dim, slots + 1, 1)``
  classifies the rendered map per pixel (label rendering of instance slots, a softmax over them).
- **Losses**: the run's loss set gives 3DGS's colour terms (``+loss=image``, 0.8 L1 + 0.2 D-SSIM); the family's own
  terms (``hooks.loss_terms``) are ``identity``, the pixel-mean cross-entropy of the classified map against the mask
  ids over ln(slots + 1), and ``identity_3d``, the k-nearest-neighbour KL of the Gaussians' class distributions over
  ``slots + 1`` every ``reg3d_every`` steps (``loss_utils.loss_cls_3d``), weighted by ``model.loss_weights``.
- **Density**: the public ``DefaultStrategy`` on 3DGS's schedule, densifying until 10k of 30k steps.

What differs from the official code, and why, is in the package's README.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Mapping

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import (
    DataError,
    GaussianFamily,
    GaussianHooks,
    GaussianScene,
    GaussianSetup,
    ImageOutput,
    Predicts,
    Prediction,
    SemanticMode,
    SemanticOutput,
    SourceViews,
    StepBatch,
    StepOutput,
    TargetCamera,
    TrainingState,
)


class GroupingHooks(GaussianHooks):
    """3DGS's hooks (``GaussianHooks``) and Gaussian Grouping's two loss terms."""

    family: "GaussianGrouping"

    def loss_terms(self, state: TrainingState, wanted: frozenset[str]) -> Mapping[str, Tensor]:
        family, terms = self.family, {}
        if "identity" in wanted:
            terms["identity"] = sum(family.identity_loss(view, output) for view, output
                                    in zip(state.batch.views, state.outputs.views)) / len(state.batch.views)
        if "identity_3d" in wanted:
            due = (state.step + 1) % family.reg3d["every"] == 0  # the official 1-based iteration % interval
            seed = state.batch.views[0].render_seed  # the same draw on any process, and after a resume
            terms["identity_3d"] = family.neighbour_kl(seed) if due else family.gaussians.means.new_zeros(())
        return terms


class GaussianGrouping(GaussianFamily):
    """One scene's Gaussians with identity encodings (the module docstring).

    Args:
        identity_dim: channels of each Gaussian's identity encoding.
        slots: identity classes (mask ids 0 to ``slots - 1``); the classifier has ``slots + 1`` outputs.
        reg3d: the 3D regulariser's ``every``, ``k``, ``sample_size`` and ``max_points``.
        setup: the checked options of ``GaussianSceneConfig`` (``gaussian_setup``).
    """

    name = "gaussian_grouping"
    capabilities = dataclasses.replace(GaussianFamily.capabilities, accepts_head=False,
                                       loss_terms=("identity", "identity_3d"), hooks=GroupingHooks)

    def __init__(self, *, identity_dim: int, slots: int, reg3d: Mapping[str, int], setup: GaussianSetup) -> None:
        super().__init__(channels={"identity": identity_dim}, setup=setup)
        self.slots = slots
        self.reg3d = dict(reg3d)
        self.classifier = nn.Conv2d(identity_dim, slots + 1, 1)

    @property
    def semantic_output(self) -> SemanticOutput:
        return SemanticOutput(Predicts.INSTANCES, SemanticMode.LABEL_RENDERING, self.slots + 1, self.slots)

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """The Gaussians' groups (``identity`` among them) and the classifier's (``model.lr.classifier``)."""
        return {**self.gaussian_groups(), "classifier": list(self.classifier.parameters())}

    def classify(self, identity: Tensor, size: tuple[int, int]) -> Tensor:
        """``[1, slots + 1, H, W]`` scores of a rendered ``[h, w, identity_dim]`` identity map."""
        logits = self.classifier(identity.permute(2, 0, 1)[None])
        return logits if tuple(logits.shape[-2:]) == size else F.interpolate(logits, size=size, mode="nearest")

    def forward(self, batch: StepBatch, *, semantics: bool, sample_semantics: bool = False) -> StepOutput:
        """Every view with its identity scores (its own loss terms read them, whatever the loss set reads)."""
        views = []
        for view in batch.views:
            output, identity = self.render_view(view.camera, channels=True)
            views.append(dataclasses.replace(output, scores=self.classify(identity, view.camera.image_size)))
        return StepOutput(tuple(views))

    @torch.inference_mode()
    def predict(self, camera: TargetCamera, sources: SourceViews | None, *, stride: int, chunk_rays: int,
                features: object = None) -> Prediction:
        """The view rasterized on a ``stride`` grid (0: every pixel), its identity map classified."""
        stride = stride or 1
        rgb, depth, _, identity, _ = self.render(camera, stride, channels=True)
        return Prediction(rgb=rgb, depth=depth, semantic=identity.permute(2, 0, 1),
                          logits=self.classify(identity, camera.image_size), stride=stride)

    @torch.inference_mode()
    def scene_gaussians(self, sources: SourceViews | None, *, near: float, far: float,
                        features: object = None) -> GaussianScene:
        """The Gaussians, each labelled with the slot its identity is classified to (Gaussian Grouping's 3D
        classification, as for editing); -1 where that is the "no instance" output."""
        slots = self.identity_logits().argmax(dim=-1)
        return self.gaussians.as_scene(torch.where(slots == self.slots, -1, slots))

    def identity_logits(self) -> Tensor:
        """``[G, slots + 1]`` the classifier on each Gaussian's own identity encoding."""
        weight = self.classifier.weight[:, :, 0, 0]
        return self.gaussians.identity @ weight.T + self.classifier.bias

    def identity_loss(self, view, output: ImageOutput) -> Tensor:
        """Cross-entropy of the view's identity scores against its mask ids (at the pixels its mask keeps), over
        ln(slots + 1); an id the classifier has no class for is a ``DataError`` naming the frame."""
        ids = view.instances
        if ids is None:
            raise DataError(f"model=gaussian_grouping trains on instance ids; scene {view.scene!r} frame "
                            f"{view.frame} has none")
        if int(ids.max()) >= self.slots or int(ids.min()) < 0:
            raise DataError(f"scene {view.scene!r} frame {view.frame} has instance id {int(ids.max())}; "
                            f"model.slots={self.slots} takes ids 0 to {self.slots - 1}: set model.slots > "
                            f"{int(ids.max())}")
        loss = F.cross_entropy(output.scores, ids[None], reduction="none")[0]
        if view.valid is not None:
            loss = loss[view.valid]
        return loss.mean() / math.log(self.slots + 1)

    def neighbour_kl(self, seed: int) -> Tensor:
        """Mean KL(P_i || P_j) of ``sample_size`` sampled Gaussians' class distributions to their ``k`` nearest by
        detached centre (themselves included), among at most ``max_points``, over ``slots + 1``."""
        probs = torch.softmax(self.identity_logits(), dim=-1)
        xyz = self.gaussians.means.detach()
        generator = torch.Generator(device=xyz.device).manual_seed(int(seed))
        if xyz.shape[0] > self.reg3d["max_points"]:
            keep = torch.randperm(xyz.shape[0], generator=generator, device=xyz.device)[: self.reg3d["max_points"]]
            xyz, probs = xyz[keep], probs[keep]
        chosen = torch.randperm(xyz.shape[0], generator=generator, device=xyz.device)[: self.reg3d["sample_size"]]
        nearest = torch.cdist(xyz[chosen], xyz).topk(min(self.reg3d["k"], xyz.shape[0]), largest=False).indices
        p, q = probs[chosen][:, None], probs[nearest]
        kl = (p * (torch.log(p + 1e-10) - torch.log(q + 1e-10))).sum(dim=-1).mean()
        return kl / probs.shape[1]
