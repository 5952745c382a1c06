"""Configuration: the TOML file and the command line's per-sensor options -> frozen settings."""
