"""The recorder role: every message of a fleet's keys into an MCAP file (see services.recorder.app)."""
