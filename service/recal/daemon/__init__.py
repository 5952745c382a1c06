"""The long-running processes: the gateway (`recal run`) and its ports, the remote calibration
node (`recal node`), the checkpoint store with its state-folder files, and what every such
process shares (`runtime`)."""
