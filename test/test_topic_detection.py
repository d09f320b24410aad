"""data/topic_detection: which bag topic is the camera image, camera_info, odometry - by message type, under any
names; a name needed only among several, and clear errors listing the candidates."""
import pytest

from dpv_sensor.data import rosbag_io as R
from dpv_sensor.data.topic_detection import describe_choice, detect_input_topics

USER_BAG = {'/robot/front/img': (R.IMAGE, 30), '/robot/front/calib': (R.CAMERA_INFO, 30),
            '/wheel/odometry': (R.ODOMETRY, 300), '/tf': ('tf2_msgs/msg/TFMessage', 99)}


def test_input_topics_found_by_type_under_any_names():
    chosen, how = detect_input_topics(USER_BAG)
    assert chosen == {'image': '/robot/front/img', 'camera_info': '/robot/front/calib', 'odom': '/wheel/odometry'}
    assert how['image'] == 'the only sensor_msgs/msg/Image topic'
    assert how['odom'] == 'the only nav_msgs/msg/Odometry topic'
    line = describe_choice(chosen, how)
    assert line.startswith('image /robot/front/img (the only sensor_msgs/msg/Image topic), '
                           'camera_info /robot/front/calib')


def test_two_image_topics_need_a_name_and_the_error_lists_both():
    topics = dict(USER_BAG, **{'/robot/rear/img': (R.IMAGE, 12)})
    with pytest.raises(R.BagError) as err:
        detect_input_topics(topics, options={'image': 'IMAGE_TOPIC='})
    msg = str(err.value)
    assert msg.startswith('2 sensor_msgs/msg/Image topics could be the image: ')
    assert '/robot/front/img [sensor_msgs/msg/Image, 30 messages]' in msg
    assert '/robot/rear/img [sensor_msgs/msg/Image, 12 messages]' in msg and msg.endswith('choose with IMAGE_TOPIC=')
    chosen, how = detect_input_topics(topics, image='/robot/rear/img')
    assert chosen['image'] == '/robot/rear/img' and how['image'] == 'named'


def test_camera_info_next_to_the_chosen_image_wins_among_several():
    topics = {'/cam/color/image_raw': (R.IMAGE, 5), '/cam/color/camera_info': (R.CAMERA_INFO, 5),
              '/cam/depth/camera_info': (R.CAMERA_INFO, 5), '/odom': (R.ODOMETRY, 5)}
    chosen, how = detect_input_topics(topics)
    assert chosen['camera_info'] == '/cam/color/camera_info'
    assert how['camera_info'] == 'the only sensor_msgs/msg/CameraInfo topic next to /cam/color/image_raw'
    with pytest.raises(R.BagError, match='2 sensor_msgs/msg/CameraInfo topics could be the camera_info'):
        detect_input_topics(dict(topics, **{'/cam/color/image_raw': (R.IMAGE, 5), '/other/image': (R.IMAGE, 5)}),
                              image='/other/image')


def test_node_outputs_are_never_taken_for_the_camera_and_unneeded_roles_may_be_missing():
    topics = {'/cam/image': (R.IMAGE, 5), '/ns/depth/image': (R.IMAGE, 2), '/ns/confidence/image': (R.IMAGE, 2),
              '/ns/rgb/image': (R.IMAGE, 2), '/ns/depth/camera_info': (R.CAMERA_INFO, 2),
              '/cam/camera_info': (R.CAMERA_INFO, 5)}
    chosen, how = detect_input_topics(topics, need=('image', 'camera_info'))
    assert chosen == {'image': '/cam/image', 'camera_info': '/cam/camera_info', 'odom': None}
    assert how['odom'] == 'absent'
    with pytest.raises(R.BagError, match=r'no nav_msgs/msg/Odometry topic for odom in the bag; choose with --odom'):
        detect_input_topics(topics, options={'odom': '--odom'})


def test_a_wrong_name_or_type_is_a_clear_error():
    with pytest.raises(R.BagError, match=r"no topic '/nope' for image in the bag; sensor_msgs/msg/Image topics: "
                                         r"/robot/front/img \[sensor_msgs/msg/Image, 30 messages\]"):
        detect_input_topics(USER_BAG, image='/nope')
    with pytest.raises(R.BagError, match='/wheel/odometry carries nav_msgs/msg/Odometry, image needs sensor_msgs'):
        detect_input_topics(USER_BAG, image='/wheel/odometry')
