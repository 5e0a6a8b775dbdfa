"""The ESPROS TOFcam635 (epc635): wire protocol, transports, pyusb driver, and its emulator
(firmware state machine, image sources, faults, pyusb backend, pseudo-terminal server)."""
