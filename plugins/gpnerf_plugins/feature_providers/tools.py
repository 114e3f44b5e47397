"""``python -m gpnerf_core data features +feature_provider=<name> [overrides...]``: compute a provider's features of
every frame of the configured dataset's scenes into the cache once (a progress bar over the frames), and check the
frames already there (each frame's checksum; a corrupt shard is computed again)."""

from __future__ import annotations

import sys
import time

from gpnerf_core import ArgumentParser, ConfigError, FeatureCache, build_feature_provider, compose, get_registry


def features(argv: list[str]) -> int:
    parser = ArgumentParser(
        prog="gpnerf_core data features",
        description="Fill the feature cache of +feature_provider=<name> for the configured dataset's scenes; the "
                    "other arguments are the run's Hydra overrides (dataset.*, feature_provider.*, threads=, device=).")
    parser.add_argument("--scenes", default="", help="comma-separated scene names (default: every scene of both "
                        "splits, the unseen ones first)")
    parser.add_argument("--batch", type=int, default=8, help="frames per provider call (default 8)")
    args, overrides = parser.parse_known_args(argv)
    for override in overrides:  # an unknown name is one line listing the known ones, not Hydra's search path
        group, _, value = override.lstrip("+").partition("=")
        if group in ("feature_provider", "dataset") and value:
            get_registry().get(group, value)
    cfg = compose(overrides)
    provider = build_feature_provider(cfg)
    if provider is None:
        raise ConfigError("data features needs a provider: +feature_provider=<name> (python -m gpnerf_core plugins "
                          "lists them under feature_provider)")
    import torch

    if int(cfg.threads) > 0:
        torch.set_num_threads(int(cfg.threads))
    device = str(cfg.device)
    device = ("cuda" if torch.cuda.is_available() else "cpu") if device == "auto" else device
    dataset = get_registry().build("dataset", cfg.dataset)
    known = list(dataset.scenes("unseen")) + [s for s in dataset.scenes("train") if s not in dataset.scenes("unseen")]
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()] or known
    unknown = [s for s in scenes if s not in known]
    if unknown:
        raise ConfigError(f"--scenes names {unknown[0]!r}, not a scene of dataset {cfg.dataset.name!r}; known: "
                          f"{', '.join(known)}")
    import logging

    from tqdm import tqdm

    class AboveTheBar(logging.Handler):  # a corrupt shard's warning on a line of its own, above the progress bar
        def emit(self, record: logging.LogRecord) -> None:
            tqdm.write(f"warning: {record.getMessage()}", file=sys.stderr)

    cache_log = logging.getLogger("gpnerf_core.features.cache")
    cache_log.addHandler(AboveTheBar(logging.WARNING))
    cache_log.propagate = False
    try:
        return _fill(provider, dataset, scenes, args.batch, device)
    finally:
        cache_log.handlers = [h for h in cache_log.handlers if not isinstance(h, AboveTheBar)]
        cache_log.propagate = True


def _fill(provider, dataset, scenes: list[str], batch: int, device: str) -> int:
    """Fill and check each scene's cache, a progress bar over its frames; prints the folders and the counts."""
    from tqdm import tqdm

    started = time.perf_counter()
    computed = read = 0
    for name in scenes:
        cache = FeatureCache(provider, dataset, name, batch=batch, device=device)
        missing = set(cache.missing_shards())
        with tqdm(total=cache.num_frames, desc=f"features {name}", unit="frame", file=sys.stderr,
                  dynamic_ncols=True) as bar:
            for shard in range(cache.num_shards):
                frames = list(cache.shard_range(shard))
                if shard in missing:
                    cache.fill_shard(shard, bar.update)
                else:
                    cache.features(frames)  # checks every frame's checksum; a corrupt shard is computed again
                    bar.update(len(frames))
        computed += cache.computed
        read += cache.read
        print(f"{name}: {cache.computed} frames computed, {cache.read} read from the cache "
              f"({cache.channels} x {cache.size[0]} x {cache.size[1]} per frame) in {cache.folder}")
    print(f"feature cache: {computed} frames computed, {read} read, {len(scenes)} scenes, "
          f"{time.perf_counter() - started:.1f} s; provider {provider.fingerprint()}")
    return 0
