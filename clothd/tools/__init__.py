"""clothd's tools: replay, the benchmarks and their grading. They run offline or drive the daemon from
outside; this is the only part of clothd that may import hwsim (to record scenarios and read truth)."""
