"""World families, navigation-difficulty metrics and ranking."""
