"""The lifecycle every command shares: compose and validate before anything is written, claim the run folder, set up
the process, and refuse what cannot run before any work."""
