"""The ESPROS TOFcam635 (epc635): wire protocol, transports, pyusb driver, and its emulator
(firmware state machine on an injected image source, faults, pyusb backend, pseudo-terminal server)."""
