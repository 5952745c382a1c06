"""The calibration node: one per sensor, between the bus or a recording and the core's
`Pipeline`; the parts it holds (alignment, device time, the published samples, the estimate
checks, the rate hold and layout, rediscovery), its sinks and its checkpoint document."""
