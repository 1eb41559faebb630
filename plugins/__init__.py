"""Built-in selector plugins of arraysel (installed as ``arraysel_plugins``)."""
