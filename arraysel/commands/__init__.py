"""One module per ``arraysel`` sub-command."""
