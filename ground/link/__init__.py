"""The link: the ground node's zenoh stream in (node), the journal it keeps of it, its frames put in order (arrivals), and the player that sends a recorded one again."""
