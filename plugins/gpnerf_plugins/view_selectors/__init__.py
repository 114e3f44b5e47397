"""Built-in view_selectors."""
