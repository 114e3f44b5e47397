"""The model: built from a config, its weights, trained models read back, source features kept between renders."""
