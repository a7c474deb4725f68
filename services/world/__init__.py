"""The world role: paces the simulator to the wall clock and publishes sensor frames and ground truth."""
