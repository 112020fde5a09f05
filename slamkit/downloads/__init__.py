"""Public RGB-D sequences fetched for the user (`slamkit-data download`): resumable HTTP
downloads with a checksum (`transfer`), archive extraction with an integrity check
(`archives`), and the sequences GS-ICP SLAM's paper evaluates on (`catalogue`)."""
