"""Live ROS 2 over DDS without a ROS install (``[live]`` extra: the cyclonedds binding).

- ``idl``: builtin_interfaces Time, std_msgs Header, sensor_msgs PointField / PointCloud2 and the
  other message types as IDL structs with the ROS 2 DDS type names; ROS topic name -> DDS topic name;
- ``dds``: the participant, the QoS and the loopback-only configuration tests and benchmarks use;
- ``params`` / ``params_file``: the parameter table, the command line and a ROS 2 parameters file
  read within limits; ``checks``: what the parameters mean together, checked at start;
- ``node``: ``msdnet-node``'s loop (one Pipeline, latest-message-wins); ``stats``: its counters and
  latency percentiles; ``observe``: its debug topics and periodic ``/diagnostics``; ``discovery``:
  writers on its input topic it cannot match, named once; ``lifecycle``: signals in any state and
  the one way out of the process;
- ``cli``: the ``msdnet-node`` command; ``publish``: a scan publisher (tests, benchmarks, trying it).
"""
