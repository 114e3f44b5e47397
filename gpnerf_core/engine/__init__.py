"""The lifecycle every command shares, one module per concern: ``launching`` (compose and validate before anything is
written, then Hydra), ``guarding`` (one line and an exit code per error), ``sweeps`` (a ``-m`` sweep's failed jobs),
``setup`` (validate once, set up the process), ``resuming`` (``train.resume``), ``runs`` (the run folder and its
records) and ``opening`` (a trained model opened one way)."""
