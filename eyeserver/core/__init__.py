"""Small shared value types; imports nothing else of eyeserver."""
