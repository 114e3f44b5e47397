"""GP-NeRF's context-aware decoding, for any model family that renders per-ray semantic features in its extractor's
semantic-map space (``RenderedRays.semantic``): in training the head decodes the **fused map**, the target image's own
semantic map (the teacher) with the rendered features written into the cells the rays hit; on a whole view it decodes
the rendered map (``render_whole_view`` with ``decode``). ``LabelsOrHead`` is the base of families that render class
scores without a head (label rendering) and features for a head with one.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from gpnerf_core.errors import PluginError
from gpnerf_core.interfaces.head import PerceptionHead, Predicts
from gpnerf_core.interfaces.model import Capabilities, ModelFamily, SemanticMode, SemanticOutput
from gpnerf_core.types import HeadOutput, RenderedRays, TargetView, ViewOutput


def cells_of_pixels(pixels: Tensor, image_size: tuple[int, int], map_size: tuple[int, int]) -> Tensor:
    """Flat cell index ``[R]`` of the map cell containing each pixel ``(u, v)`` ``[R, 2]``.

    Exact integer cells (``v // s_y``, ``u // s_x``), fixing the released code's off-by-one (REFERENCE C2).
    """
    height, width = image_size
    map_h, map_w = map_size
    col = torch.div((pixels[:, 0] + 0.5) * map_w, width, rounding_mode="floor").long().clamp(0, map_w - 1)
    row = torch.div((pixels[:, 1] + 0.5) * map_h, height, rounding_mode="floor").long().clamp(0, map_h - 1)
    return row * map_w + col


def pixel_cells(image_size: tuple[int, int], map_size: tuple[int, int], device: torch.device | None = None) -> Tensor:
    """``[H * W]`` the flat map cell of every pixel of an ``image_size`` image, row-major (``cells_of_pixels`` of every
    pixel): a map read at each pixel, e.g. a loss on whole images that compares two maps pixel by pixel."""
    height, width = image_size
    flat = torch.arange(height * width, device=device)
    pixels = torch.stack([flat % width, flat // width], dim=-1).to(torch.float32)
    return cells_of_pixels(pixels, image_size, map_size)


def gather_cells(feature_map: Tensor, cells: Tensor) -> Tensor:
    """Rows ``[R, C]`` of a ``[1, C, h, w]`` map at flat ``cells`` ``[R]`` (gradient preserved)."""
    return feature_map.flatten(2)[0, :, cells].T


def fuse_rendered(teacher: Tensor, rendered: Tensor, cells: Tensor) -> Tensor:
    """Replace the teacher's cells hit by rays with the rendered features (averaged where rays share a cell).

    Args:
        teacher: ``[1, C, h, w]`` target-view semantic map; keeps its gradient in the cells no ray hits.
        rendered: ``[R, C]`` rendered features; cells: ``[R]`` flat cell indices.

    Returns:
        ``[1, C, h, w]`` fused map.
    """
    _, channels, map_h, map_w = teacher.shape
    flat = teacher.flatten(2)[0]  # [C, h * w]
    sums = torch.zeros_like(flat).index_add(1, cells, rendered.T.to(flat.dtype))
    counts = torch.bincount(cells, minlength=map_h * map_w).to(flat.dtype)
    hit = counts > 0
    fused = torch.where(hit[None, :], sums / counts.clamp_min(1.0)[None, :], flat)
    return fused.reshape(1, channels, map_h, map_w)


def decode_checked(head: PerceptionHead, semantic_map: Tensor, output_size: tuple[int, int]) -> HeadOutput:
    """``head`` on a ``[N, C, h, w]`` semantic map; its output is checked against the contract (``[N, num_outputs,
    *output_size]``)."""
    output = head(semantic_map, output_size)
    logits = getattr(output, "logits", None)
    expected = [int(semantic_map.shape[0]), int(head.num_outputs), int(output_size[0]), int(output_size[1])]
    if not isinstance(output, HeadOutput) or not isinstance(logits, Tensor) or list(logits.shape) != expected:
        found = list(logits.shape) if isinstance(logits, Tensor) else type(output).__name__
        raise PluginError(
            f"head {type(head).__name__} returned {found}; the PerceptionHead contract is "
            f"HeadOutput(logits=[N, num_outputs, *output_size]) = {expected}"
        )
    return output


def decoded_view_output(view: TargetView, coarse: RenderedRays, fine: RenderedRays | None, teacher: Tensor,
                        head: PerceptionHead, *, fuse: bool = True) -> ViewOutput:
    """A training view's outputs around its rendered features: the teacher at the rays' cells, the fused map (or the
    teacher alone where ``fuse`` is False: the released code) and the head's logits on it.

    Args:
        view: the target view (its pixels and camera).
        coarse, fine: the passes; the last one's ``semantic`` ``[R, C]`` are the rendered features.
        teacher: ``[1, C, h, w]`` the extractor's semantic map of the target image (not detached).
    """
    camera = view.camera
    cells = cells_of_pixels(view.pixels, camera.image_size, (int(teacher.shape[-2]), int(teacher.shape[-1])))
    last = fine if fine is not None else coarse
    head_input = fuse_rendered(teacher, last.semantic, cells) if fuse else teacher
    return ViewOutput(coarse=coarse, fine=fine, teacher_map=teacher, teacher_at_rays=gather_cells(teacher, cells),
                      head_input=head_input, logits=decode_checked(head, head_input, camera.image_size).logits)


def labels_or_head_output(head: PerceptionHead | None, num_classes: int) -> SemanticOutput | None:
    """The ``semantic_output`` of a family whose scores are ``head``'s (decoded: its classes or instance slots), or
    without a head its own K = ``num_classes`` class scores per pixel (label rendering); None with neither."""
    if head is not None:
        predicts = Predicts(head.predicts)
        slots = getattr(head, "slots", None) if predicts is Predicts.INSTANCES else None
        return SemanticOutput(predicts, SemanticMode.DECODED, int(head.num_outputs), slots)
    if not num_classes:
        return None
    return SemanticOutput(Predicts.CLASSES, SemanticMode.LABEL_RENDERING, num_classes)


class LabelsOrHead(ModelFamily):
    """A family whose semantic outputs are K class scores composited per ray (label rendering) without a head, and
    features decoded by ``head`` with GP-NeRF's context-aware decoding with one (``decoded_view_output``; on a whole
    view ``render_whole_view`` with ``decode``). What such a family says about itself is the same for all: it sets
    ``extractor`` (a ``FeatureExtractor``), ``head`` (or None) and ``num_classes`` (K, 0 with a head or without labels).
    """

    capabilities = Capabilities(teacher=True)

    extractor: nn.Module
    head: PerceptionHead | None
    num_classes: int

    @property
    def semantic_output(self) -> SemanticOutput | None:
        return labels_or_head_output(self.head, self.num_classes)

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """The extractor under ``feature_extractor``, the head under ``head``, the family's own networks under
        ``transformer``."""
        own = [p for name, p in self.named_parameters() if not name.startswith(("extractor.", "head."))]
        groups = {"feature_extractor": list(self.extractor.parameters()), "transformer": own}
        if self.head is not None:
            groups["head"] = list(self.head.parameters())
        return groups

    @torch.inference_mode()
    def teacher_logits(self, image: Tensor) -> Tensor | None:
        """With a head: the head on the target image's own semantic map (the 2D-only reference)."""
        if self.head is None:
            return None
        return decode_checked(self.head, self.extractor(image[None]).semantic, tuple(image.shape[-2:])).logits
