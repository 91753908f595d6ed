"""The built-in ROS 2 actions (one ``<name>.py`` + ``<name>.umrf.json`` each); ``docs/ros2.md``."""
