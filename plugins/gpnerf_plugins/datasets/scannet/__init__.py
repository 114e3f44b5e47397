"""ScanNet: the ``scannet`` dataset, its file parsers, labels, checker, splits and the ``.sens`` converter."""
