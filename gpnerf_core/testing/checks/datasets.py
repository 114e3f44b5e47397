"""Checks of datasets that need no files: the class map and the config. Loading scenes needs the data itself."""

from __future__ import annotations

from gpnerf_core.testing.checks.common import CheckFailed, CheckSkipped, Subject, call, check_round_trip, expect


def check_classes(subject: Subject) -> None:
    """``class_names`` a tuple of str (empty only for a dataset of unlabelled scenes, whose model brings its own list),
    ``num_classes`` their count, an int ``ignore_index`` outside [0, K)."""
    try:
        dataset = subject.build()
    except CheckFailed as failure:
        raise CheckSkipped(f"it does not build without its files here ({failure})") from None
    names = call("reading class_names", lambda: dataset.class_names)
    expect(isinstance(names, tuple) and all(isinstance(n, str) and n for n in names),
           f"class_names is {names!r:.80}, expected a tuple of non-empty str")
    count = call("reading num_classes", lambda: dataset.num_classes)
    expect(count == len(names), f"num_classes is {count!r} but class_names has {len(names)} names")
    ignore = call("reading ignore_index", lambda: dataset.ignore_index)
    expect(isinstance(ignore, int) and not isinstance(ignore, bool), f"ignore_index is {ignore!r}, expected an int")
    expect(not 0 <= ignore < count, f"ignore_index {ignore} is a valid class id in [0, {count}); it must not be one")


CHECKS = {
    "classes": check_classes,
    "config round trip": check_round_trip,
}
