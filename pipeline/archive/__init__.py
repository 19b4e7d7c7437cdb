"""``rsmb survey``: a night of captures into a survey folder, its ledger and index page."""
