"""The channel role: the V2X link emulator, an application-level relay around mapcontainer.channel."""
