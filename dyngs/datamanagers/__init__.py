"""Dataset parsers (one per on-disk format) and the datamanager that serves batches."""
