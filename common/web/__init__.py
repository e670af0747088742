"""What the browser-facing servers share (the operator page, the video signalling).

web_token.py: the secrets that open the local web sockets; bounded_json.py:
JSON from a peer with its nesting bounded.
"""
