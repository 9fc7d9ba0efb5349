"""The service around the online twin: rig configuration, per-rig runners and worker processes, Zenoh bus, journal, store, live view."""
