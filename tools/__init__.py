"""Repository tooling for tests and benchmarks: random-weight checkpoints, services and robots on loopback.

Not part of the product: the wheel ships schemas/, client/ and service/ only.
"""
