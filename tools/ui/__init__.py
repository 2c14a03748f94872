"""``drivectl ui``: the commissioning console in a browser, on the same session as the shell (docs/ui.md)."""
