"""The photo going in: safe decoding, the object's mask (the salient-object net, a person's box and strokes,
GrabCut) and the framing the networks expect."""
