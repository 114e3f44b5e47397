"""The plugin registry: the component kinds, the hooks, loading plugins and building what they register."""
