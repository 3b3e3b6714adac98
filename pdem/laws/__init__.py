"""Built-in contact laws, registered through pdem's own entry points like any plugin."""
