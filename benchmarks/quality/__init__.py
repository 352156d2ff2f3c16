"""``msdnet-bench quality``: the quality suite (``suite``), its keys (``columns``), writers (``report``)."""
