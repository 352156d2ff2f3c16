"""``msdnet-bench latency``: the timing suite (``suite``) and its parts.

``cli`` (click command), ``models`` (model pairs), ``timing`` and ``runs`` (timed stages), ``compare``
(int8 and torch comparisons), ``quality`` (quality by loop steps), ``report`` (results writers).
"""
