"""User-facing errors: one line, the bad value, what is allowed, exit code 2."""


class UsageError(Exception):
    """Bad input from the user. The CLI prints `error: <message>` and exits with code 2, never a traceback."""


def check_choice(name: str, value, allowed) -> None:
    if value not in allowed:
        raise UsageError(f"unknown {name} {value!r}; allowed: {', '.join(map(str, allowed))}")


def check_non_negative(name: str, value) -> None:
    if value is None or value < 0:
        raise UsageError(f"{name} must be >= 0, got {value!r}")


def check_positive(name: str, value) -> None:
    if value is None or value <= 0:
        raise UsageError(f"{name} must be > 0, got {value!r}")
