"""Built-in feature providers (``+feature_provider=<name>``): xfeat, files, teacher, open_clip, timm; and the
``data features`` tool that fills their cache."""
