"""xmetro_ros.bag."""
