"""Recordings of other tools into session files: ADI ToF dumps, Azure Kinect (Matroska),
replay of session files as a device; :mod:`.dispatch` detects the format (``import_file``)."""
