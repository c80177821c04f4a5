"""xmetro_ros.loop."""
