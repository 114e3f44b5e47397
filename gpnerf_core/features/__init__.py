"""Feature providers' 2D features and the feature fields distilled from them (docs/features.md)."""
