"""Training infrastructure: the LightningCLI wrapper behind `segmo fit/validate/test`."""
