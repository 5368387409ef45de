"""The pure controller: the step and the reference generators."""
