"""Readers and writers: files, layouts, datasets, bags, Rerun recordings, pictures.

- ``files``: ``read_cloud`` / ``write_cloud`` (``.bin``, ``.txt``, ``.npy``, ``.pcd``, ``.ply``);
  ``atomic``: atomic writes and the temporary files a killed run leaves; ``layouts``: named
  ``.bin`` layouts;
- ``datasets``: the VoD, Astyx and simulator dataset readers, their preprocessing
  (``datasets.preprocess``) and realism statistics (``datasets.stats``);
- ``rosbag``: ROS 1/2 bags and PointCloud2 messages; ``bag_guards``: checks around a bag written;
  ``pairing``: a bag's radar and LiDAR -> a VoD-layout training folder;
- ``rerun_log``: Rerun recordings; ``pictures``: bird's-eye-view PNGs.
"""
