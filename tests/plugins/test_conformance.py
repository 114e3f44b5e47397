"""Every built-in component passes the contract kit that third-party plugins run (``gpnerf_core.testing``).

One test item per component and check, at small sizes so the whole file stays fast.
"""

from gpnerf_core.registry.plugins import BUILTIN_PLUGINS
from gpnerf_core.registry.kinds import KINDS
from gpnerf_core.testing import contract_checks, plugin_checks

pytest_plugins = ["gpnerf_core.testing.pytest_plugin"]

SMALL = {
    "feature_extractor/resunet_fpn": {"widths": [8, 8, 16, 16], "blocks": [1, 1, 1], "radiance_dim": 8,
                                      "fpn_channels": 8},
    "field_aggregator/gnt_view": {"width": 16, "num_blocks": 2, "pos_frequencies": 2},
    "head/unet": {"channels": 16, "norm_groups": 4},
    # MVSNeRF's own extractor (mvsnet) makes no semantic maps, which the kit's head decodes: the one with them
    "model/mvsnerf": {"feature_extractor": {"name": "resunet_fpn"}},
    "head/per_pixel": {"hidden_dim": 16},
    # the kit makes 3DGS's density control act within its steps itself (KIT_DENSITY)
    "model/semantic_3dgs": {"init_points": 300, "feature_dim": 4, "sh_degree": 1},
    # anchors that fit the kit's 32 x 48 frames; narrow heads
    "model/mask_rcnn": {"anchor_sizes": [4.0, 8.0, 16.0, 24.0, 32.0], "fpn_channels": 8, "box_hidden": 16,
                        "mask_hidden": 8, "roi_batch_size_per_image": 16, "slots": 8},
}


@contract_checks(BUILTIN_PLUGINS, configs=SMALL)
def test_contract(gpnerf_check):
    gpnerf_check.run()


def test_every_kind_has_a_checked_builtin_component():
    checked = {check.component.split("/")[0] for check in plugin_checks(BUILTIN_PLUGINS)}
    assert checked == set(KINDS) | {"stress_case"}
