"""Device files as worn accelerometers write them: Axivity .cwa (.cwa.gz), GENEActiv .bin,
ActiGraph .gt3x, read with actfast and recognised by content (`registry.KINDS`)."""

from recal.io.device_files.recording import DeviceRecording, is_device_file, open_device
from recal.io.device_files.registry import KINDS, sniff

__all__ = ["KINDS", "DeviceRecording", "is_device_file", "open_device", "sniff"]
