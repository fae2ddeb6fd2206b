"""gcdtrav client library: talk to the service over Zenoh (no torch)."""
