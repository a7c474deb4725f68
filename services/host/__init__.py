"""The host role: the fusion container fed from Zenoh; the solver runs in a worker process."""
