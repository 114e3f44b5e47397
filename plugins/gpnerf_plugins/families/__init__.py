"""Model families: what renders a target view's rays (``model=<name>``)."""
