"""The glance between the schedule and inference: a frame's grey block thumbnail and the pose's motion (change),
and the triage that settles an unchanged view by reusing its last maps (reuse)."""
