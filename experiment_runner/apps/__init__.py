"""The applications of nanostage, on top of the core and the ROS layer: the ``nanostage``
command line, bench, warm-up, ``graph``/``replay``, the design advisor, campaigns, diagnosis
and the paper reproduction. Independent of each other (``.importlinter``)."""
