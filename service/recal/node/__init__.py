"""The calibration node: one per sensor, between the bus or a recording and the core's
`Pipeline`; its sinks, its alignment requests, its checkpoint document and re-discovery."""
