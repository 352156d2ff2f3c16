"""``msdnet-data``: ``cli`` (the command group), ``show_stats`` (``show``, ``stats``), ``pair``
(``pair``; the work is in ``io/pairing``); ``simulate`` is ``sim.command``.
"""
