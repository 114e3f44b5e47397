"""``python -m gpnerf_core.tools.viewer.timing``: the preview and full-frame seconds docs/viewer.md reports."""

from gpnerf_core.tools.viewer.timing import measure
from pipeline_check import TINY_MODEL, TINY_SCENES


def test_timing_reports_preview_and_full_frame_seconds_and_cpu_time(tiny):
    result = measure(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, "view.stride=4"], repeats=1)
    assert result["image"] == [32, 48] and (result["stride"], result["preview_stride"]) == (4, 8)
    for key in ("preview_s_cold", "preview_s_warm", "full_s_cold", "full_s_warm"):
        assert 0 <= result[key] < 60, key
    assert result["cpu_user_s"] > 0 and result["cpu_system_s"] >= 0 and result["minor_page_faults"] >= 0
    assert result["peak_resident_mb"] > 0
    # a query on the kept full frame: GP-NeRF's semantic embedding at stride 4's grid, no render
    assert 0 < result["query_s"] < 0.1 and result["query_features"] == "semantic_embedding"
    assert result["query_grid"][1:] == [8, 12]
