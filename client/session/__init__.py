"""Zenoh session helpers shared by the library and the commands: configuration from arguments, publisher identity."""
