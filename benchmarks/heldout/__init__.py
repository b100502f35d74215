"""The held-out validation set of issue 55 (item 8): independent plants and a frozen case table."""
