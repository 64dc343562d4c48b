"""π0-style hybrid: a Llama backbone over [images, text, state] and a flow-matching action expert on its K/V."""
