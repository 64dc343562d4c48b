"""vlactl: observe and steer vision-language-action policies through their internal representations."""

__version__ = "0.1.0"
