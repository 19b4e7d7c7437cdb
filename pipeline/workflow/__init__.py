"""``rsmb run``: nightly workflow files, validated and run step by step."""
