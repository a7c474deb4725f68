"""Zenoh services: one OS process per role, each a thin adapter around a core class of mapcontainer."""
