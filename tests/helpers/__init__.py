"""Helpers the tests share: the golden release cases, the reference renderer, Chromium, quick
training configs, data-format writers, and a process that holds a file open mid-write."""
