"""Recordings of other tools into session files: ADI ToF dumps, Azure Kinect (Matroska), ROS 2
bags (MCAP, :mod:`.ros2`, which also writes sessions as bags), replay of session files as a
device; :mod:`.dispatch` detects the format (``import_file``)."""
