"""The HIL loop: the control cycle, the lockstep and real-time runners, and the run session."""
