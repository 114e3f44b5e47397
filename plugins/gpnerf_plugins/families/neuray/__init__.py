"""NeuRay + semantic head (``model=neuray``) and Semantic-Ray (``model=semantic_ray``): occlusion-aware aggregation over
source views with label rendering; Semantic-Ray adds its Cross-Reprojection Attention."""
