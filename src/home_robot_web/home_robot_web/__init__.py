"""The robot's web page (``web_ui_node``): functional core in plain Python, a thin ROS shell."""
