"""What is read out of a finished store: queries, derived quantities, exports, pictures."""
