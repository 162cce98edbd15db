"""Shared test helpers (import these, not other test modules): ``processes`` starts the project's
commands in a child process the one way the tests do."""
