"""tofhil.drivers: frames from ToF cameras, real and emulated, and recordings of other tools.

- ``base``: the driver interface, the device registry (``open_device("emulator")``,
  ``list_devices()``) and capture settings; ``capture``: frames of a device into a session;
- ``tofcam635``: the ESPROS TOFcam635 (protocol, USB and serial transports, the pyusb
  driver, and its emulator); ``depthai``: Luxonis ToF cameras through DepthAI v3 (device and
  host-only pipelines);
- ``importers``: ADI ToF frames, Azure Kinect recordings, ROS 2 bags (MCAP, in and out),
  replay of sessions;
- ``sources``: where an emulated device's images come from (a frame source its caller
  injects: drivers never import the simulator).
"""

from tofhil.faces import lazy_face

__all__, __getattr__, __dir__ = lazy_face(__name__, {
    "open_device": "base",
    "create_driver": "base",
    "list_devices": "base",
    "register_driver": "base",
    "CaptureSettings": "base",
    "Driver": "base",
    "import_file": "importers.dispatch",
    "provide_frame_sources": "sources",
})
