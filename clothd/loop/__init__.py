"""The loop: the daemon's tick, the compute process it drives, and the state it publishes."""
