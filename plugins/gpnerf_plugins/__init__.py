"""Built-in plugins of gpnerf-core; each subpackage registers through its plugin.py hooks only."""
