"""Serving a policy: the server and its encoding (`server`), B1K's evaluation harness (`harness`);
the entry point is `pi0_armfix.serve`."""
