"""Why a policy fails: ACT hooks, representation diagnostics, the prompt-swap probe, attention views, the report."""
