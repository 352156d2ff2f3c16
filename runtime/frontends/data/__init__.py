"""``msdnet-data``: simulate, show, stats, pair."""
