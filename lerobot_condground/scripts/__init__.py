"""One module per `condground` command: its config and `main`."""
