"""The frame's second room: the newest frame per source waits in the latest-only queue; the share's policy
picks which source's frame goes next (a ready frame's claim, the one every-other-turn rule)."""
