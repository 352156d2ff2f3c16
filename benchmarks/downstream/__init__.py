"""``msdnet-bench odometry`` / ``place``: the downstream suite (``suite``) and its parts.

``odometry`` (scan-to-scan GICP), ``place`` (ScanContext recall@K).
"""
