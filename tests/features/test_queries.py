"""Queries by example and by embedding on synthetic features: the similarity map peaks at the example, a box averages
its cells, prototypes from labelled pixels label a map perfectly, a query of another dimension is refused naming both,
and a selection is its own PLY that a reader of the format alone reads back."""

from __future__ import annotations

import pytest
import torch

from gpnerf_core import (
    class_prototypes, example_embedding, nearest_prototype, select_gaussians, similarity_map, write_gaussian_selection,
    write_point_selection,
)
from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.evaluation import metrics as M
from gpnerf_core.features.queries import cell_labels, feature_stride, text_embedding
from gpnerf_core.geometry.gaussians.scene import GaussianScene
from ply_reader import read_ply


def regions(channels: int = 8, grid=(6, 8)) -> tuple[torch.Tensor, torch.Tensor]:
    """A ``[C, h, w]`` map of three regions (left, right top, right bottom), each its own random direction plus a
    little noise, and its ``[h, w]`` labels."""
    generator = torch.Generator().manual_seed(3)
    directions = torch.randn(3, channels, generator=generator)
    labels = torch.zeros(grid, dtype=torch.long)
    labels[: grid[0] // 2, grid[1] // 2:] = 1
    labels[grid[0] // 2:, grid[1] // 2:] = 2
    features = directions[labels].permute(2, 0, 1) + 0.05 * torch.randn(channels, *grid, generator=generator)
    return features * 3.0, labels  # a scale cosine ignores


def test_the_similarity_map_of_a_pixel_example_peaks_at_the_example_and_its_region():
    features, labels = regions()
    stride = 8  # the map of a 48 x 64 image
    query = example_embedding(features, pixel=(63.0, 5.0), stride=stride)  # cell (0, 7): region 1
    similarity = similarity_map(features, query)
    assert similarity.shape == (6, 8) and float(similarity[0, 7]) == pytest.approx(1.0, abs=1e-5)
    assert float(similarity.max()) == pytest.approx(float(similarity[0, 7]))
    assert float(similarity[labels == 1].min()) > float(similarity[labels != 1].max())
    assert float(similarity.min()) >= -1.0 - 1e-5


def test_a_box_example_is_the_mean_of_the_normalised_cells_it_covers():
    features, labels = regions()
    query = example_embedding(features, box=(0, 0, 15, 47), stride=8)  # columns 0-1, every row: region 0
    unit = features / features.norm(dim=0, keepdim=True)
    assert torch.allclose(query, unit[:, :, :2].reshape(8, -1).mean(dim=1), atol=1e-6)
    assert float(similarity_map(features, query)[labels == 0].min()) > 0.9
    with pytest.raises(ConfigError, match="outside the 48x64 image"):
        example_embedding(features, pixel=(64, 0), stride=8)
    with pytest.raises(ConfigError, match="exactly one"):
        example_embedding(features, stride=8)
    with pytest.raises(ConfigError, match="x0 <= x1"):
        example_embedding(features, box=(20, 0, 10, 5), stride=8)
    assert feature_stride(features, (48, 64)) == 8


def test_prototypes_from_labelled_pixels_label_a_map_perfectly():
    features, labels = regions()
    full = labels.repeat_interleave(4, 0).repeat_interleave(4, 1)  # the labels at the 24 x 32 image
    prototypes = class_prototypes([features], [full], num_classes=4, ignore_index=255)
    assert prototypes.shape == (4, 8) and torch.isnan(prototypes[3]).all()  # class 3: no labelled pixel
    predicted = nearest_prototype(features, prototypes)
    assert torch.equal(predicted, labels)
    scores = M.image_scores_from_confusion(M.confusion_matrix(predicted, labels, 4))
    assert scores[M.MIOU_IMAGE_MEAN_PRESENT] == 1.0


def test_cell_labels_take_each_cells_most_frequent_label():
    labels = torch.tensor([[0, 0, 1, 255], [0, 1, 255, 255]])
    assert cell_labels(labels, (1, 2), 2, 255).tolist() == [[0, 255]]


def test_a_grid_that_does_not_divide_the_image_maps_pixels_and_labels_proportionally():
    features, labels = regions()  # 6 x 8 cells, as a provider rounds a 50 x 66 frame at stride 8
    query = example_embedding(features, pixel=(65.0, 49.0), image_size=(50, 66))  # the last cell
    assert torch.allclose(query, features[:, 5, 7] / features[:, 5, 7].norm(), atol=1e-6)
    full = torch.nn.functional.interpolate(labels[None, None].float(), size=(50, 66), mode="nearest")[0, 0].long()
    assert torch.equal(cell_labels(full, (6, 8), 3), labels)
    prototypes = class_prototypes([features], [full], num_classes=3)
    assert torch.equal(nearest_prototype(features, prototypes), labels)


def test_a_query_of_another_dimension_is_refused_naming_both():
    features, _ = regions(channels=8)
    with pytest.raises(ConfigError, match=r"^the query embedding has 5 dimensions and the feature field has 8 "
                                          r"channels; expected a query of 8 values") as refused:
        similarity_map(features, torch.ones(5))
    assert "\n" not in str(refused.value)
    with pytest.raises(ConfigError, match="has 3 dimensions and the feature field has 8 channels"):
        select_gaussians(torch.ones(10, 8), torch.ones(3), 0.5)
    with pytest.raises(ConfigError, match="has 4 dimensions and the feature map has 8 channels"):
        nearest_prototype(features, torch.ones(2, 4))
    with pytest.raises(ConfigError, match="threshold 1.5"):
        select_gaussians(torch.ones(10, 8), torch.ones(8), 1.5)


class _Provider:
    def encode_text(self, texts):
        return torch.stack([torch.full((8,), float(len(t))) for t in texts])


def test_a_text_query_is_the_providers_embedding():
    assert torch.equal(text_embedding(_Provider(), "chair"), torch.full((8,), 5.0))
    with pytest.raises(ConfigError, match="query text is empty"):
        text_embedding(_Provider(), "  ")


def gaussians(count: int, channels: int = 4) -> GaussianScene:
    generator = torch.Generator().manual_seed(1)
    return GaussianScene(means=torch.randn(count, 3, generator=generator), scales=torch.full((count, 3), 0.01),
                         rotations=torch.tensor([[1.0, 0, 0, 0]]).repeat(count, 1), opacities=torch.full((count,), 0.5),
                         harmonics=torch.rand(count, 3, 4, generator=generator),
                         labels=torch.arange(count), features=torch.randn(count, channels, generator=generator))


def test_the_selected_gaussians_are_their_own_ply_read_back_from_the_format(tmp_path):
    scene = gaussians(20)
    query = scene.features[3]
    selected = select_gaussians(scene.features, query, 0.5)
    assert bool(selected[3]) and 0 < int(selected.sum()) < 20
    scores = torch.nn.functional.cosine_similarity(scene.features, query[None], dim=1)
    path = write_gaussian_selection(tmp_path / "selection.ply", scene, selected, scores)
    columns = read_ply(path.read_bytes())
    assert columns["label"].tolist() == torch.nonzero(selected).flatten().tolist()  # the selected rows, in order
    assert torch.allclose(torch.from_numpy(columns["x"]), scene.means[selected, 0])
    assert (columns["relevancy"] >= 0.5 - 1e-6).all() and "f_dc_0" in columns and "rot_3" in columns
    with pytest.raises(DataError, match="none of the 20 Gaussians is selected"):
        write_gaussian_selection(tmp_path / "none.ply", scene, torch.zeros(20, dtype=torch.bool))
    assert not (tmp_path / "none.ply").exists()


def test_the_selected_points_are_their_own_ply(tmp_path):
    xyz, rgb = torch.rand(10, 3), torch.rand(10, 3)
    selected = torch.arange(10) % 3 == 0
    columns = read_ply(write_point_selection(tmp_path / "points.ply", xyz, rgb, selected).read_bytes())
    assert torch.allclose(torch.from_numpy(columns["y"]), xyz[selected, 1])
    assert columns["red"].tolist() == (rgb[selected, 0] * 255).round().to(torch.uint8).tolist()
