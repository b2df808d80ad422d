"""Runtime: executors and signals, progress and cancellation."""
