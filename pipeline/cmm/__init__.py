"""The CMM wing: the ROMER line protocol, the other arm line formats, and point-file readers."""
