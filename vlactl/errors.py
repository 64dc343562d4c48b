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


def check_device(name: str, value):
    """A torch device this machine has, e.g. cpu, cuda, cuda:1 -> torch.device."""
    import torch  # here, not at the top: the CLI's error path should not pay for torch

    try:
        device = torch.device(str(value))
    except RuntimeError:
        raise UsageError(f"{name} {value!r} is not a torch device; allowed: cpu, cuda, cuda:<index>") from None
    if device.type == "cuda" and (not torch.cuda.is_available() or (device.index or 0) >= torch.cuda.device_count()):
        raise UsageError(f"{name} {value!r}: torch sees {torch.cuda.device_count()} CUDA GPU(s) here; use {name}=cpu")
    if device.type not in ("cpu", "cuda"):
        raise UsageError(f"{name} {value!r} is not supported; allowed: cpu, cuda, cuda:<index>")
    return device
