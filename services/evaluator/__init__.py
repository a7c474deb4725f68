"""The evaluator role: live accuracy, latency and bandwidth figures of a running fleet."""
