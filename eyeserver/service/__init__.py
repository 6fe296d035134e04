"""The running daemon: rig lifecycle, acquisition, jobs, tracking, state machine, storage."""
