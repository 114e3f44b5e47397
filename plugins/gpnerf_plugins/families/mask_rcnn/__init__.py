"""Mask R-CNN (He et al., ICCV 2017) as a 2D instance baseline of Table 2, in plain torch: ``model=mask_rcnn``."""
