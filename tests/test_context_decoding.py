import torch

from gpnerf_core.model.context_decoding import cells_of_pixels, fuse_rendered, gather_cells


def test_cells_are_exact_stride_cells_without_wraparound():
    pixels = torch.tensor([[0.0, 0.0], [1.0, 1.0], [2.0, 0.0], [7.0, 5.0], [6.0, 4.0]])
    cells = cells_of_pixels(pixels, (6, 8), (3, 4))
    assert cells.tolist() == [0, 0, 1, 11, 11]


def test_fused_map_writes_rendered_cells_and_averages_duplicates():
    teacher = torch.arange(2 * 3 * 4, dtype=torch.float32).reshape(1, 2, 3, 4).requires_grad_()
    rendered = torch.tensor([[100.0, 200.0], [300.0, 400.0], [-1.0, -2.0]], requires_grad=True)
    cells = torch.tensor([5, 5, 0])
    fused = fuse_rendered(teacher, rendered, cells)
    assert fused[0, :, 1, 1].tolist() == [200.0, 300.0]
    assert fused[0, :, 0, 0].tolist() == [-1.0, -2.0]
    untouched = torch.ones(3, 4, dtype=torch.bool)
    untouched[1, 1] = untouched[0, 0] = False
    assert torch.equal(fused[0][:, untouched], teacher[0][:, untouched])
    fused.sum().backward()
    # the teacher keeps its gradient only where no ray was rendered
    assert teacher.grad[0, 0, 1, 1] == 0 and teacher.grad[0, 0, 2, 3] == 1
    assert torch.equal(rendered.grad, torch.tensor([[0.5, 0.5], [0.5, 0.5], [1.0, 1.0]]))


def test_gather_cells_reads_rows():
    feature_map = torch.arange(2 * 2 * 3, dtype=torch.float32).reshape(1, 2, 2, 3)
    rows = gather_cells(feature_map, torch.tensor([0, 4]))
    assert rows.tolist() == [[0.0, 6.0], [4.0, 10.0]]
