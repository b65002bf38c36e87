"""What a person sees of a running deployment: the status book and its text, and the screen."""
