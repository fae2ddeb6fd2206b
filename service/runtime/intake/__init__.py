"""The frame's first room: a payload arrives and is admitted or refused before it takes a slot: the intake rate
per publisher, the source cap and its candidates, the capture stamp read without decoding, each source's
clock, the one age rule (freshness). Admission offers what it admits to the schedule."""
