"""Dataset readers (one per dataset, common conventions in base.py), shards and loaders."""
