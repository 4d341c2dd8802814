"""Wire messages: what the processes say to each other, their encoding and their validity rules."""
