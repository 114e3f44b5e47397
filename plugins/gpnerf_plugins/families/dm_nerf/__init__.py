"""DM-NeRF (Wang et al., ICLR 2023) as a per-scene instance family: ``model=dm_nerf``."""
