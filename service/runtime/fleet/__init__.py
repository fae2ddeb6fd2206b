"""Beside the frame's order: what instances of a fleet share. Which instance takes which source (assignment), the
credits a source's owner grants when its slot frees, one model and one anchor set per fleet, and the anchor
set's switch, its state file and the lock that keeps one service per state file."""
