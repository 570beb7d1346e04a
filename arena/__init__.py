"""Arena: the contract every service shares (keys, messages, config, Zenoh session, CLI)."""

__version__ = "0.1.0"
