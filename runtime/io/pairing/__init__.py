"""``msdnet-data pair``: a ROS bag with a radar and a LiDAR topic -> a VoD-layout training folder.

- ``transforms``: the radar-to-LiDAR extrinsic (``--extrinsic`` or ``/tf_static``) and poses
  (``/tf`` or an odometry topic), a small TF tree with interpolation;
- ``pair``: stamp pairing and the writer of the VoD layout; ``command``: the click command.
"""
