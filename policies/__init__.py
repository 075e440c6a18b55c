"""Policies of the plugin. The `act_modified` policy type lands here (issue 3)."""
