"""The long-running processes: the gateway (`recal run`), the remote calibration node
(`recal node`) and what every such process shares (`runtime`)."""
