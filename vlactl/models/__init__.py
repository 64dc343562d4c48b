"""VLA models behind one small interface (`base.VLA`); one file or folder per model, resolved by name in `registry`."""
