
FB1/IN 8
FB1/X 8P