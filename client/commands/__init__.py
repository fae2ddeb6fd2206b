"""The client's commands: `gcdtrav status`, `anchors`, `probe`, `relay`, `view` and the container health check."""
