"""xmetro_ros.sim."""
