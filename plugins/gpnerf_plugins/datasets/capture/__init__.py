"""A user's own capture: nerfstudio's transforms.json read as a dataset, and the tools that make one."""
