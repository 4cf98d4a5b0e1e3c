"""Training code (never run by `make test`): fine-tuning matchers on synthetic pairs."""
