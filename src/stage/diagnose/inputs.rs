//! The diagnosis stage's inputs: the work directory's tables read into the plain data of
//! [`crate::diagnose::locate`].
