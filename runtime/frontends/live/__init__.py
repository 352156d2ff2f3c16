"""Live ROS 2 over DDS without a ROS install (``[live]`` extra: the cyclonedds binding).

- ``idl``: builtin_interfaces Time, std_msgs Header, sensor_msgs PointField / PointCloud2 as IDL
  structs with the ROS 2 DDS type names; ROS topic name -> DDS topic name;
- ``dds``: the participant, the QoS and the loopback-only configuration tests and benchmarks use;
- ``node``: ``msdnet-node``'s loop (one Pipeline, latest-message-wins, latency percentiles);
- ``cli``: the ``msdnet-node`` command; ``publish``: a scan publisher (tests, benchmarks, trying it).
"""
