"""The ``instance`` head: GP-NeRF's context-aware decoder with ``slots + 1`` instance outputs."""

from __future__ import annotations

from dataclasses import dataclass

from gpnerf_core import ConfigError, Predicts
from gpnerf_plugins.heads.unet import UNetHead


@dataclass
class InstanceHeadConfig:
    """Options of the ``instance`` head."""

    name: str = "instance"
    """Registry name of the head."""
    slots: int = 16
    """Instance slots K; the head outputs K + 1 channels (the last: no instance). At least the most instance ids
    (background included) any training frame holds."""
    decoder: str = "semantic_fpn"
    """'semantic_fpn' (the reference's recommended instance decoder) or 'unet' (the paper's U-Net form)."""
    channels: int = 128
    """Width of every decoder conv."""
    norm_groups: int = 32
    """GroupNorm groups; must divide ``channels``."""


class InstanceHead(UNetHead):
    """The ``unet`` head's decoders with instance outputs: logits ``[N, slots + 1, H, W]``, softmax over channels.

    Args:
        in_dim, in_levels: runtime sizes (see ``ResizingHead``).
        num_outputs: ``slots + 1``, supplied by the pipeline from ``slots``.
        slots: instance slots K.
        decoder, channels, norm_groups: as for ``UNetHead``.
    """

    predicts = Predicts.INSTANCES

    def __init__(
        self,
        in_dim: int,
        in_levels: int,
        num_outputs: int,
        slots: int = InstanceHeadConfig.slots,
        decoder: str = InstanceHeadConfig.decoder,
        channels: int = InstanceHeadConfig.channels,
        norm_groups: int = InstanceHeadConfig.norm_groups,
    ) -> None:
        if slots < 1:
            raise ConfigError(f"head.slots={slots}: expected a positive number of instance slots")
        if num_outputs != slots + 1:
            raise ConfigError(f"instance head got num_outputs={num_outputs}; expected head.slots + 1 = {slots + 1}")
        super().__init__(in_dim, in_levels, num_outputs, decoder=decoder, channels=channels, norm_groups=norm_groups)
        self.slots = int(slots)
