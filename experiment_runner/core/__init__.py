"""The ROS-free core of experiment_runner: the batch engine, reference profiles, metrics,
experiments, recordings, outputs, task execution, table import, nominal models and the
user-input errors. It imports no rclpy, no ROS-layer module and no application
(``.importlinter``, contract ``layers``)."""
