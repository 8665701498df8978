"""The scheduler process and everything with I/O (specs, runner, store, HTTP, CLI)."""
