"""xmetro_ros.learn."""
