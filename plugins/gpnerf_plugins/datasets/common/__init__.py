"""Code shared by more than one dataset: image decoding, layout-check reports, dataset root folders."""
