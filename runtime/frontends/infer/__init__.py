"""``msdnet-infer``: ``cli`` (the command), ``files`` (file mode: here, ``--workers`` processes, Ray),
``worker`` (the per-file work every file mode shares), ``guards`` (``--out``, worker count, killed
parents), ``dataset`` (``--dataset``), ``bag`` (``BAG --topic``), ``ray_batch`` (``--ray``).
"""
