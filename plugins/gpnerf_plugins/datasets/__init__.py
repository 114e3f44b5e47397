"""Built-in datasets: one subpackage per dataset (embedded, replica, scannet), shared code in common/."""
